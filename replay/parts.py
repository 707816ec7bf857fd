"""A series of parts cut by one NC program, with part-to-part variation and tool wear (known truth).

A process monitor learns its references from the first good parts of a program and watches the
rest; to test it, every part must differ the way real parts do and no more. Part i of a series of a
process scenario (``[series]`` of ``replay/scenarios/_process.toml``) is the scenario with

* material factor ``m_i ~ N(1, material_std)`` clipped at ±3σ (stock lot hardness) times the wear
  factor ``w_i = 1 + wear_per_part · i`` (tool wear: the force grows by ``wear_per_part`` per part),
  both on the cutting coefficients, so the cutting force is ``∝ m_i w_i``;
* spindle speed ``s_i n`` with ``s_i ~ U(1 − spindle_rel, 1 + spindle_rel)``, the programmed feed
  rate kept (the chip ``c/s_i`` changes, as on a machine programmed in mm/min);
* feed override ``o_i ~ U(1 − feed_override_rel, 1 + feed_override_rel)``: the feed rate and chip ×
  ``o_i``, the time of every feed section ÷ ``o_i`` (the path is the same);
* a random spindle angle at the start (``phase``) and its own noise seed;
* the scenario's process events (tooth break, runout growth, collision, missing stock) from part
  ``events_from_part`` on; the parts before it are good parts (the event happens in a running series).

Part i is drawn from its own random stream ``(seed, i)``: the first parts of a series of 20 are the
first parts of a series of 200. One trial file per part, ``part-0000.mcap`` …, each with a ``part``
truth event (t = 0, value = i, the part's factors in ``detail``) and the factors in
``provenance.details["part"]``; with a start time given, part i starts ``gap_s`` after part i − 1
ends, so the files form one production timeline.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from feedio import schema as S
from feedio.mcapio import format_time, parse_time

from . import scenarios as SC

__all__ = ["PartVariation", "MAX_PARTS", "series_constants", "part_variations", "part_duration", "part_scenario",
           "simulate_series", "truth_sections"]

#: most parts one series may hold (one trial file each)
MAX_PARTS = 100_000
_STREAM_PART = 0x9A27  # the random stream of the part-to-part variation (apart from the simulator's streams)
_SERIES_LIMITS = {  # key → (lowest, highest)
    "material_std": (0.0, 0.2),
    "spindle_rel": (0.0, 0.3),
    "feed_override_rel": (0.0, 0.5),
    "wear_per_part": (0.0, 0.1),
    "gap_s": (0.0, 86400.0),
}


@dataclass(frozen=True)
class PartVariation:
    """The constants that make part ``index`` differ from the programme (factors relative to it)."""

    index: int
    events: bool  # the scenario's process events happen in this part (index ≥ events_from_part)
    material: float  # m_i, stock lot
    wear: float  # w_i = 1 + wear_per_part · i
    spindle: float  # s_i, spindle speed factor
    feed_override: float  # o_i
    phase_deg: float  # spindle angle at t = 0, degrees
    seed: int  # the simulator's noise seed
    start_s: float  # start of the part from the start of the series, s

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def series_constants(sc: dict, wear_per_part: float | None = None) -> dict:
    """The scenario's ``[series]`` table, checked (ValueError naming the constant and its range)."""
    if "series" not in sc or "process" not in sc:
        raise ValueError(f"scenario {sc.get('name', '?')!r} has no [series] table: a part series needs a process "
                         "scenario (milling-part and the other milling scenarios built on _process)")
    out = dict(sc["series"])
    if wear_per_part is not None:
        out["wear_per_part"] = wear_per_part
    for key, (lo, hi) in _SERIES_LIMITS.items():
        v = out[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and lo <= v <= hi):
            raise ValueError(f"series.{key} must be a number in [{lo:g}, {hi:g}], got {v!r}")
    k = out["events_from_part"]
    if isinstance(k, bool) or not isinstance(k, int) or not 0 <= k <= MAX_PARTS:
        raise ValueError(f"series.events_from_part must be a whole number 0 … {MAX_PARTS}, got {k!r}")
    if not isinstance(out["phase"], bool):
        raise ValueError(f"series.phase must be true or false, got {out['phase']!r}")
    return out


def part_duration(sc: dict, override: float) -> float:
    """Length of a part (s) at feed override ``override``: the feed sections take 1/override as long."""
    tr = sc["trajectory"]
    return tr["lead_in"] + tr["lead_out"] + (sc["duration"] - tr["lead_in"] - tr["lead_out"]) / override


def part_variations(sc: dict, n_parts: int, *, seed: int = 0, wear_per_part: float | None = None) -> list[PartVariation]:
    """The variation of parts ``0 … n_parts − 1`` (each from its own random stream ``(seed, i)``)."""
    if isinstance(n_parts, bool) or not isinstance(n_parts, int) or not 1 <= n_parts <= MAX_PARTS:
        raise ValueError(f"a series holds 1 … {MAX_PARTS} parts, got {n_parts!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be an integer ≥ 0, got {seed!r}")
    c = series_constants(sc, wear_per_part)
    out, start = [], 0.0
    for i in range(n_parts):
        rng = np.random.default_rng([seed, _STREAM_PART, i])
        z = float(np.clip(rng.standard_normal(), -3.0, 3.0))
        spindle = 1.0 + c["spindle_rel"] * rng.uniform(-1.0, 1.0)
        override = 1.0 + c["feed_override_rel"] * rng.uniform(-1.0, 1.0)
        phase = float(rng.uniform(0.0, 360.0)) if c["phase"] else float(sc["disturbance"]["phase"])
        sim_seed = int(np.random.SeedSequence([seed, i]).generate_state(1)[0])
        out.append(PartVariation(index=i, events=i >= c["events_from_part"], material=1.0 + c["material_std"] * z,
                                 wear=1.0 + c["wear_per_part"] * i,
                                 spindle=spindle, feed_override=override, phase_deg=phase, seed=sim_seed,
                                 start_s=start))
        start += part_duration(sc, override) + c["gap_s"]
    return out


def part_scenario(sc: dict, var: PartVariation) -> dict:
    """The scenario of one part: the programme with the part's factors (see the module docstring)."""
    out = copy.deepcopy(sc)
    d = out["disturbance"]
    d["spindle_rpm"] = float(d["spindle_rpm"]) * var.spindle
    d["phase"] = var.phase_deg
    # levels are mm per tooth at the scenario's speed: the feed rate follows the override only
    out["trajectory"]["levels"] = [x * var.feed_override / var.spindle for x in sc["trajectory"]["levels"]]
    out["duration"] = part_duration(sc, var.feed_override)
    p = out["process"]
    p["material"] = float(sc["process"]["material"]) * var.material * var.wear
    if not var.events:  # a good part: no breaks, runout growth, collisions or missing stock
        p["breaks"], p["impulses"], p["missing"] = [], [], []
        p["runout_growth_m_per_s"] = []
    SC.check(out)
    return out


def simulate_series(sc: dict, n_parts: int, out_dir, *, seed: int = 0, created: str | None = None,
                    wear_per_part: float | None = None, fine: bool = False, first: int = 0,
                    progress=None) -> list[Path]:
    """Simulate parts ``first … n_parts − 1`` of the series of scenario dict ``sc`` and write
    ``out_dir/part-NNNN.mcap`` (``out_dir`` is created). ``created``: start time of part 0 (ISO 8601),
    later parts follow on the series' timeline; None: each file starts when written.
    ``progress(i, path)`` is called after each part. Returns the paths written."""
    from .simulator import simulate, write_trial

    variations = part_variations(sc, n_parts, seed=seed, wear_per_part=wear_per_part)
    start_ns = None if created is None else parse_time(created, what="created")
    out_dir = Path(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    width = max(4, len(str(n_parts - 1)))
    paths = []
    for var in variations[first:]:
        part_sc = part_scenario(sc, var)
        stamp = None if start_ns is None else format_time(start_ns + int(round(var.start_s * 1e9)))
        res = simulate(part_sc, seed=var.seed, fine=fine, created=stamp)
        res.meta.provenance.details["part"] = var.to_dict()
        res.events.insert(0, S.TruthEvent(kind="part", t_s=0.0, seq=0, value=float(var.index), detail=var.to_dict()))
        path = out_dir / f"part-{var.index:0{width}d}.mcap"
        write_trial(res, path)
        paths.append(path)
        if progress is not None:
            progress(var.index, path)
    return paths


def truth_sections(res) -> list[dict]:
    """The per-section statistics of a simulated part from its true force, in the form of
    :meth:`monitor.process_monitor.AxisProcessMonitor.finish` (tool, program_line, occurrence, rows,
    mean_force_N, energy_J = Σ F·v·Ts): the wear monitor's input without the estimator, for its statistics."""
    line, tool = np.asarray(res.program_line), np.asarray(res.tool)
    f, v = np.asarray(res.force, dtype=np.float64), np.asarray(res.v_true, dtype=np.float64)
    ts = float(res.meta.Ts)
    cut = np.flatnonzero((line[1:] != line[:-1]) | (tool[1:] != tool[:-1])) + 1
    out, seen = [], {}
    for a, b in zip(np.r_[0, cut], np.r_[cut, line.size]):
        key = (int(tool[a]), int(line[a]))
        occ = seen[key] = seen.get(key, -1) + 1
        out.append({"tool": key[0], "program_line": key[1], "occurrence": occ, "rows": int(b - a),
                    "mean_force_N": float(f[a:b].mean()), "energy_J": float((f[a:b] * v[a:b]).sum() * ts)})
    return out
