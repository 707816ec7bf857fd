"""The axis model file: what ``feedmon identify`` writes and ``feedmon run`` reads.

TOML, human-readable, versioned (``format_version``), never pickled. One file per
axis. Layout (version 1)::

    format_version = 1

    [axis]            machine, axis
    [model]           form, Ts (s), beta, beta_names, omega (m/s), coulomb,
                      loop_gain (N·s/m, optional), method
    [physical]        inertia (kg), damping (N·s/m), coulomb_pos/neg (N), offset (N),
                      or inertia_over_gain (s), damping_over_gain when K is unknown
    [tracker]         kernel, sigma1 (s), sigma2, period (s), gamma, forgetting,
                      budget, jitter — the online KRLS-T (method §6); kernel = "spindle"
                      with per, teeth, spindle_rpm instead of period: the spindle-phase
                      kernel (:mod:`monitor.online_settings`)
    [adaptation]      online β (optional; :class:`monitor.online_settings.Adaptation`)
    [health]          health thresholds (optional; :class:`monitor.online_settings.Health`)
    [identification]  sigma1, sigma2, period, gamma used by PL-LSSVM, tuned, log_likelihood
    [provenance]      source, sha256, method, created, feedmon_version

:func:`load_model` validates every key and raises :class:`ModelFileError`
naming the key and the file; :func:`save_model` writes the same layout.
"""

from __future__ import annotations

import hashlib
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from kernels.covariance import Kernel
from kernels.feed_drive import FORMS, beta_names

from . import online_settings as OS

__all__ = [
    "FORMAT_VERSION",
    "ModelFileError",
    "TrackerConfig",
    "AxisModel",
    "load_model",
    "save_model",
    "file_sha256",
]

FORMAT_VERSION = 1


class ModelFileError(ValueError):
    """A model file that cannot be used; the message names the file and the key."""


@dataclass
class TrackerConfig:
    """KRLS-T hyperparameters for the online tracker (method §6), defaults after thesis Table 4.5."""

    kernel: dict = field(default_factory=lambda: {"type": "locally_periodic", "sigma1": OS.TRACKER_DEFAULTS["sigma1"],
                                                  "sigma2": OS.TRACKER_DEFAULTS["sigma2"], "period": 1 / 55})
    gamma: float = OS.TRACKER_DEFAULTS["gamma"]
    forgetting: float = OS.TRACKER_DEFAULTS["forgetting"]
    budget: int = OS.TRACKER_DEFAULTS["budget"]
    jitter: float = OS.TRACKER_DEFAULTS["jitter"]

    def build_kernel(self) -> Kernel:
        return OS.build_tracker_kernel(self.kernel)


@dataclass
class AxisModel:
    """Everything the monitor needs for one axis."""

    machine: str
    axis: str
    form: str
    Ts: float
    beta: list[float]
    omega: float
    coulomb: bool
    tracker: TrackerConfig
    loop_gain: float | None = None
    method: str = "pl-lssvm"
    physical: dict = field(default_factory=dict)
    identification: dict = field(default_factory=dict)
    provenance: dict = field(default_factory=dict)
    online: OS.OnlineSettings = field(default_factory=OS.OnlineSettings)  # [adaptation], [health]

    @property
    def beta_names(self) -> tuple[str, ...]:
        return beta_names(self.form, self.coulomb)

    @property
    def force_scalable(self) -> bool:
        """True when a disturbance can be published in newtons (method §6)."""
        return self.form == "force-input" or self.loop_gain is not None

    @property
    def force_gain(self) -> float | None:
        """``b = K_d/K`` (m/s per N) or None: ``F = −f / b``."""
        if self.form == "force-input":
            return self.beta[0]
        if self.loop_gain is not None:
            return self.beta[0] / self.loop_gain
        return None


# ---------------------------------------------------------------------------
# loading with validation
# ---------------------------------------------------------------------------


class _Reader:
    def __init__(self, path: Path, doc: dict):
        self.path = path
        self.doc = doc

    def fail(self, key: str, problem: str) -> ModelFileError:
        return ModelFileError(f"{self.path}: key '{key}': {problem}")

    def table(self, name: str, required: bool = True) -> dict:
        value = self.doc.get(name)
        if value is None:
            if required:
                raise self.fail(name, f"missing table [{name}]; re-create the file with 'feedmon identify'")
            return {}
        if not isinstance(value, dict):
            raise self.fail(name, f"must be a table [{name}], got {type(value).__name__}")
        return value

    def get(self, table: str, key: str, kind, *, required: bool = True, default=None):
        t = self.table(table, required=required)
        full = f"{table}.{key}"
        if key not in t:
            if required:
                raise self.fail(full, "missing")
            return default
        value = t[key]
        if kind is float:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise self.fail(full, f"must be a number, got {type(value).__name__} {value!r}")
            value = float(value)
            if not math.isfinite(value):
                raise self.fail(full, f"must be finite, got {value!r}")
            return value
        if kind is int:
            if isinstance(value, bool) or not isinstance(value, int):
                raise self.fail(full, f"must be an integer, got {type(value).__name__} {value!r}")
            return value
        if not isinstance(value, kind):
            raise self.fail(full, f"must be of type {kind.__name__}, got {type(value).__name__} {value!r}")
        return value

    def positive(self, table: str, key: str, *, required: bool = True, default=None, allow_zero: bool = False):
        value = self.get(table, key, float, required=required, default=default)
        if value is None:
            return None
        if value < 0 or (value == 0 and not allow_zero):
            raise self.fail(f"{table}.{key}", f"must be {'≥' if allow_zero else '>'} 0, got {value!r}")
        return value

    def finite_table(self, name: str) -> dict:
        out = {}
        for key, value in self.table(name, required=False).items():
            if isinstance(value, float) and not math.isfinite(value):
                raise self.fail(f"{name}.{key}", f"must be finite, got {value!r}")
            out[key] = value
        return out


def load_model(path) -> AxisModel:
    """Read and validate a model file; errors name the file and the key (never executes anything)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise ModelFileError(f"{path}: model file not found; create one with 'feedmon identify TRIAL.mcap -o {path}'") from None
    try:
        doc = tomllib.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ModelFileError(f"{path}: not a valid TOML model file ({exc})") from None
    r = _Reader(path, doc)
    version = doc.get("format_version")
    if version is None:
        raise r.fail("format_version", "missing; is this a feedmon model file?")
    if version != FORMAT_VERSION:
        raise r.fail("format_version", f"unknown version {version!r}; this feedmon reads version {FORMAT_VERSION}")

    form = r.get("model", "form", str)
    if form not in FORMS:
        raise r.fail("model.form", f"unknown input form {form!r}; use one of {', '.join(FORMS)}")
    coulomb = r.get("model", "coulomb", bool)
    beta = r.get("model", "beta", list)
    expected = len(beta_names(form, coulomb))
    if len(beta) != expected:
        raise r.fail("model.beta", f"has {len(beta)} entries; the {form} form with coulomb={str(coulomb).lower()} needs {expected}")
    for i, b in enumerate(beta):
        if isinstance(b, bool) or not isinstance(b, (int, float)) or not math.isfinite(b):
            raise r.fail(f"model.beta[{i}]", f"must be a finite number, got {b!r}")
    names = r.get("model", "beta_names", list, required=False)
    if names is not None and tuple(names) != beta_names(form, coulomb):
        raise r.fail("model.beta_names", f"{names} do not match the {form} form (expected {list(beta_names(form, coulomb))})")

    tracker_table = r.table("tracker")
    kind = r.get("tracker", "kernel", str)
    keys = ("sigma1", "sigma2", "per", "teeth", "spindle_rpm") if kind == OS.SPINDLE else \
        ("sigma1", "sigma2", "period", "lengthscale")
    kernel_desc = {k: v for k, v in tracker_table.items() if k in keys}
    kernel_desc["type"] = kind
    for k, v in kernel_desc.items():
        if kind != OS.SPINDLE and k != "type" and (isinstance(v, bool) or not isinstance(v, (int, float))
                                                  or not math.isfinite(v) or v <= 0):
            raise r.fail(f"tracker.{k}", f"must be a positive finite number, got {v!r}")
    try:
        OS.check_kernel_desc(kernel_desc)
    except ValueError as exc:
        raise r.fail("tracker.kernel", str(exc)) from None
    forgetting = r.positive("tracker", "forgetting", required=False, default=OS.TRACKER_DEFAULTS["forgetting"])
    if forgetting > 1:
        raise r.fail("tracker.forgetting", f"must be in (0, 1], got {forgetting!r}")
    budget = r.get("tracker", "budget", int, required=False, default=OS.TRACKER_DEFAULTS["budget"])
    if budget < 1:
        raise r.fail("tracker.budget", f"must be ≥ 1, got {budget!r}")
    tracker = TrackerConfig(
        kernel=kernel_desc,
        gamma=r.positive("tracker", "gamma"),
        forgetting=forgetting,
        budget=budget,
        jitter=r.positive("tracker", "jitter", required=False, default=OS.TRACKER_DEFAULTS["jitter"], allow_zero=True),
    )
    try:
        online = OS.parse_model_tables(doc, path)
    except ValueError as exc:
        raise ModelFileError(str(exc)) from None
    return AxisModel(
        machine=r.get("axis", "machine", str),
        axis=r.get("axis", "axis", str),
        form=form,
        Ts=r.positive("model", "Ts"),
        beta=[float(b) for b in beta],
        omega=r.positive("model", "omega", allow_zero=True),
        coulomb=coulomb,
        loop_gain=r.positive("model", "loop_gain", required=False),
        method=r.get("model", "method", str, required=False, default="pl-lssvm"),
        tracker=tracker,
        physical=r.finite_table("physical"),
        identification=r.finite_table("identification"),
        provenance=dict(r.table("provenance", required=False)),
        online=online,
    )


# ---------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"model files hold finite numbers only, got {value!r}")
        return repr(value)
    if isinstance(value, str):
        escaped = value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")
        return f'"{escaped}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if hasattr(value, "item"):  # numpy scalar
        return _toml_value(value.item())
    raise TypeError(f"cannot write {type(value).__name__} to a model file")


def _table(name: str, items: dict, comments: dict | None = None) -> list[str]:
    lines = [f"[{name}]"]
    for key, value in items.items():
        if value is None:
            continue
        note = (comments or {}).get(key)
        lines.append(f"{key} = {_toml_value(value)}" + (f"  # {note}" if note else ""))
    return lines + [""]


_UNITS = {
    "Ts": "s",
    "omega": "m/s, Coulomb dead band",
    "loop_gain": "N·s/m, velocity-loop gain K",
    "inertia": "kg",
    "damping": "N·s/m",
    "coulomb_pos": "N",
    "coulomb_neg": "N",
    "offset": "N",
    "inertia_over_gain": "s (J/K)",
    "damping_over_gain": "1 (B/K)",
    "sigma1": "s",
    "period": "s (ψ)",
    "spindle_rpm": "rpm, nominal: used without spindle data",
    "per": "revolution (2π: runout) | tooth (2π/teeth)",
}


def save_model(model: AxisModel, path) -> Path:
    """Write ``model`` as a version-1 TOML model file (atomic replace)."""
    path = Path(path)
    tracker = {"kernel": model.tracker.kernel["type"]}
    tracker.update({k: v for k, v in model.tracker.kernel.items() if k not in ("type", "dims")})
    tracker.update(gamma=model.tracker.gamma, forgetting=model.tracker.forgetting, budget=model.tracker.budget, jitter=model.tracker.jitter)
    lines = [
        "# feedmon axis model (written by 'feedmon identify'; units SI)",
        f"format_version = {FORMAT_VERSION}",
        "",
        *_table("axis", {"machine": model.machine, "axis": model.axis}),
        *_table(
            "model",
            {
                "form": model.form,
                "Ts": float(model.Ts),
                "beta": [float(b) for b in model.beta],
                "beta_names": list(model.beta_names),
                "omega": float(model.omega),
                "coulomb": bool(model.coulomb),
                "loop_gain": None if model.loop_gain is None else float(model.loop_gain),
                "method": model.method,
            },
            _UNITS,
        ),
        *_table("physical", {k: v for k, v in model.physical.items()}, _UNITS),
        *_table("tracker", tracker, _UNITS),
        *_table("identification", model.identification, _UNITS),
        *[line for name, items, notes in OS.model_tables(model.online) for line in _table(name, items, notes)],
        *_table("provenance", model.provenance),
    ]
    text = "\n".join(lines)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)
    return path


def file_sha256(path) -> str:
    """Hex SHA-256 of a file (provenance of trials and model files)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
