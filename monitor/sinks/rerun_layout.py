"""What the Rerun dashboard shows: entity paths, units, series styles and the blueprint.

One axis: paths below ``/<machine>/<axis>``; ``<g>`` is ``force`` (N) when the model scales to
newtons, else ``disturbance`` (velocity disturbance in µm/s). "At" is the sample each value is
placed at, for a value from EstimateBlock row j.

* ``<g>/estimate`` filtered disturbance (``force`` / ``f``), at j−1; ``<g>/upper``, ``<g>/lower``
  estimate ± 2σ, at j−1; ``sigma/estimate`` its σ, at j−1.
* ``<g>/prediction`` one-step prediction (``force_next`` / ``f_next``), at j; ``sigma/prediction``.
* ``<g>/actual`` the truth (TruthBlock ``force`` / ``f``) of sample j; ``force/dynamometer`` the
  dynamometer reading of sample j with its sign turned to the disturbance's (the dynamometer
  measures along the axis, the disturbance force opposes motion).
* ``velocity/reference|measured|predicted`` v_ref, v_meas, v_pred in mm/s, at j.
* ``context/program_line|tool`` the NC program line and tool number of sample j (when the samples
  carry them), at j.
* ``dictionary/size`` KRLS-T dictionary size; ``dictionary/pruned|reduced`` elements pruned and
  REDUCED updates per second over the last ``rate_window`` s, at j.
* ``residual_psd/residual``, ``disturbance_psd/estimate|actual``: BarCharts, PSD in dB above the
  signal's floor vs Hz, at the last sample of their window; ``psd_markers/1_over_psi|
  tooth_passing|spindle`` marker bars (Hz) shown in both spectra.
* ``events``: TextLog (flags, gaps, glitches, spectrum markers, health, process alarms), at the sample
  concerned.
* with the process monitors on: ``force/limit/*`` their limits,
  ``force/marker/<kind>`` their alarms, ``tooth/*`` the per-tooth panel (:mod:`monitor.sinks.rerun_monitors`).

Entity names sort so that the estimate is drawn over the truth (Rerun draws in path order).

Row j of an EstimateBlock is emitted when sample j arrives; its filtered values describe sample
j−1 and its prediction sample j (docs/estimates.md, "What a value describes, in time"), so each value
is placed on the ``sample`` (sequence) and ``time`` (controller time, s) timelines at the sample
it describes and lines up with the truth of that sample.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from feedio.schema import TOOTH_VIEW_REVOLUTIONS

__all__ = ["AxisInfo", "describe_model", "Series", "series_styles", "group_of", "units_of", "AxisView",
           "axis_blueprint", "blueprint_for", "MARKER_COLOURS", "SPECTRUM_COLOURS", "TIMELINE", "SEQUENCE",
           "TOOTH_COLOUR", "ALARM_MARKER_SIZE", "alarm_style"]

TIMELINE = "time"  # controller time (s), duration timeline
SEQUENCE = "sample"  # sample sequence number

# colours (RGBA): band translucent so the estimate and the truth stay visible through it
_RED = (214, 39, 40, 255)
_BAND = (255, 110, 110, 110)
_ORANGE = (255, 160, 40, 255)
_GREEN = (70, 200, 90, 255)
_GREY = (170, 170, 170, 255)
_BLUE = (60, 150, 230, 255)
_VIOLET = (180, 130, 230, 255)
_CYAN = (23, 190, 207, 255)

_YELLOW = (230, 200, 40, 255)
_MAGENTA = (230, 60, 200, 255)
_ALARM = (255, 255, 255, 255)  # white: over the red estimate
TOOTH_COLOUR = (0, 200, 230, 255)
#: px of an alarm's marker on the force panel
ALARM_MARKER_SIZE = 16.0

MARKER_COLOURS = {"1_over_psi": (255, 215, 0, 150), "tooth_passing": (0, 220, 255, 150), "spindle": (0, 220, 255, 150)}
SPECTRUM_COLOURS = {"residual": (196, 140, 110, 255), "estimate": _RED, "actual": _GREEN}


@dataclass(frozen=True)
class Series:
    """Style of one plotted series: legend label, RGBA colour, line width (px), zoomed-out aggregation.

    ``aggregation`` is Rerun's AggregationPolicy: MinMax keeps the peaks of a 100 Hz force visible
    when a pixel covers many samples (averaging would wash them out), Max/Min keep the band's
    outer edge.
    """

    label: str
    colour: tuple[int, int, int, int]
    width: float = 1.5
    aggregation: str = "MinMax"


def group_of(force: bool) -> str:
    """Entity group of the disturbance: ``force`` (N) or ``disturbance`` (µm/s)."""
    return "force" if force else "disturbance"


def units_of(force: bool) -> str:
    return "N" if force else "µm/s"


def _disturbance_series(force: bool) -> dict[str, Series]:
    g = group_of(force)
    s = {
        f"{g}/upper": Series("estimate + 2σ", _BAND, 1.0, "Max"),
        f"{g}/lower": Series("estimate − 2σ", _BAND, 1.0, "Min"),
        f"{g}/actual": Series("true force" if force else "true disturbance", _GREEN, 1.5),
        f"{g}/estimate": Series("filtered estimate", _RED, 1.5),
        f"{g}/prediction": Series("one-step prediction", _ORANGE, 1.5),
        "sigma/estimate": Series("σ filtered estimate", _RED, 1.5, "Max"),
        "sigma/prediction": Series("σ one-step prediction", _ORANGE, 1.5, "Max"),
    }
    if force:
        s["force/dynamometer"] = Series("dynamometer (sign flipped)", _GREY, 1.0)
    return s


_COMMON: dict[str, Series] = {
    "velocity/reference": Series("reference v_ref", _GREY, 1.5),
    "velocity/measured": Series("measured v_meas", _BLUE, 1.5),
    "velocity/predicted": Series("one-step prediction v_pred", _ORANGE, 1.0),
    "dictionary/size": Series("size (elements)", _CYAN, 1.5, "MinMax"),
    "dictionary/pruned": Series("pruned per s", _VIOLET, 1.5, "Max"),
    "dictionary/reduced": Series("REDUCED per s (newest pruned at once)", _GREY, 1.0, "Max"),
}
_CONTEXT: dict[str, Series] = {
    "context/program_line": Series("NC program line", _VIOLET, 1.5, "Max"),
    "context/tool": Series("tool number", _GREY, 1.5, "Max"),
}


_PROCESS: dict[str, Series] = {  # the process monitors' limits (rerun_monitors.py), the per-tooth amplitudes
    "force/limit/collision_high": Series("collision limit, upper", _YELLOW, 1.0, "Max"),
    "force/limit/collision_low": Series("collision limit, lower", _YELLOW, 1.0, "Min"),
    "force/limit/overload_high": Series("overload limit", _MAGENTA, 1.0, "Max"),
    "force/limit/overload_low": Series("overload limit (−)", _MAGENTA, 1.0, "Min"),
    "force/limit/band_high": Series("reference band, upper", _VIOLET, 1.0, "Max"),
    "force/limit/band_low": Series("reference band, lower", _VIOLET, 1.0, "Min"),
    "tooth/a0": Series("mean force a0", _GREY, 1.5, "Average"),
    "tooth/a1": Series("once-per-revolution amplitude A1", TOOTH_COLOUR, 1.5, "Max"),
    "tooth/a1_broken": Series("A1 limit: broken tooth", _RED, 1.0, "Max"),
    "tooth/a1_runout": Series("A1 limit: runout", _ORANGE, 1.0, "Max"),
}


def alarm_style(kind: str) -> Series:
    """The style of the alarm markers of ``kind`` (``force/marker/<kind>``): a white cross named by its kind."""
    return Series(f"ALARM {kind}", _ALARM, ALARM_MARKER_SIZE)


def series_styles(force: bool, context: bool = False, process: bool = False) -> dict[str, Series]:
    """Every time series of one axis (path relative to ``/<m>/<a>``) and its style."""
    return {**_disturbance_series(force), **_COMMON, **(_CONTEXT if context else {}),
            **(_PROCESS if process and force else {})}


# ---- what the dashboard knows of an axis ------------------------------------------------------------
@dataclass(frozen=True)
class AxisInfo:
    """What the dashboard knows of an axis beyond its blocks (all optional).

    ``period`` ψ of the tracker kernel (s, 1/ψ marker), ``teeth`` of the tool (tooth-passing
    marker, with the samples' ``spindle_rpm``), ``Ts`` sampling period (s; else measured from
    the blocks), ``force``: the model scales to newtons (else decided by the first estimate).
    """

    period: float | None = None
    teeth: int | None = None
    Ts: float | None = None
    force: bool | None = None

    @classmethod
    def parse(cls, key: str, value: Mapping[str, Any]) -> AxisInfo:
        if not isinstance(value, Mapping):
            raise ValueError(f"axis_info[{key!r}] must be a mapping, got {type(value).__name__}")
        unknown = set(value) - {"period", "teeth", "Ts", "force"}
        if unknown:
            raise ValueError(f"axis_info[{key!r}]: unknown keys {sorted(unknown)}; known: period, teeth, Ts, force")
        for name in ("period", "Ts"):
            v = value.get(name)
            if v is not None and not (isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
                                      and 0 < v < 1e6):
                raise ValueError(f"axis_info[{key!r}][{name!r}] must be a positive number of seconds, got {v!r}")
        teeth = value.get("teeth")
        if teeth is not None and not (isinstance(teeth, int) and not isinstance(teeth, bool) and 1 <= teeth <= 1000):
            raise ValueError(f"axis_info[{key!r}]['teeth'] must be an integer 1..1000, got {teeth!r}")
        force = value.get("force")
        if force is not None and not isinstance(force, bool):
            raise ValueError(f"axis_info[{key!r}]['force'] must be true or false, got {force!r}")
        return cls(value.get("period"), teeth, value.get("Ts"), force)


def describe_model(model, teeth: int | None = None) -> dict[str, Any]:
    """``axis_info`` entry of an :class:`~monitor.model_file.AxisModel`: ψ of a time-periodic tracker
    kernel (s), Ts, force scaling, and the tool's teeth (argument, else a ``teeth`` attribute of the
    model when it has one)."""
    kernel = model.tracker.kernel  # a monitor.online_settings.TrackerKernel
    period = kernel.period if kernel.kind in ("locally_periodic", "locally_periodic_zero_mean", "periodic") else None
    if kernel.kind == "spindle":  # the spindle-phase kernel: its period in time at the nominal speed
        per_rev = 60.0 / float(kernel.spindle_rpm)
        period = per_rev / int(kernel.teeth) if kernel.per == "tooth" else per_rev
        if teeth is None:
            teeth = kernel.teeth
    if teeth is None:
        teeth = getattr(model, "teeth", None)
    return {"period": float(period) if period else None, "Ts": float(model.Ts), "force": bool(model.force_scalable),
            "teeth": teeth}


# ---- blueprint -------------------------------------------------------------------------------------------
def _window(seconds: float | None):
    import rerun.blueprint as rrb

    if seconds is None:
        return None
    return rrb.VisibleTimeRange(TIMELINE, start=rrb.TimeRangeBoundary.cursor_relative(seconds=-float(seconds)),
                                end=rrb.TimeRangeBoundary.cursor_relative())


def _series_view(origin: str, name: str, window: float | None, contents=None, legend: str | None = "LeftTop"):
    import rerun.blueprint as rrb

    kw = {} if contents is None else {"contents": contents}
    plot_legend = rrb.PlotLegend(visible=False) if legend is None else rrb.PlotLegend(corner=legend)
    tr = _window(window)
    if tr is not None:
        kw["time_ranges"] = tr
    return rrb.TimeSeriesView(origin=origin, name=name, plot_legend=plot_legend, **kw)


@dataclass(frozen=True)
class AxisView:
    """One axis on the dashboard: entity root (``/<m>/<a>``, escaped), names, newtons or velocity units,
    whether its samples carry context columns (NC program line, tool), whether process monitors judge it."""

    root: str
    machine: str
    axis: str
    force: bool = True
    context: bool = False
    process: bool = False


def force_view(ax: AxisView, window: float | None, title_prefix: str = ""):
    """The disturbance panel: filtered estimate ±2σ at its sample time, truth, dynamometer."""
    what = "force" if ax.force else "disturbance (velocity units)"
    name = (f"{title_prefix}{ax.axis} {what} ({units_of(ax.force)}): filtered estimate ±2σ at its sample time, "
            f"true{', dynamometer' if ax.force else ''}"
            f"{'; monitor limits, alarms (white crosses)' if ax.process and ax.force else ''}")
    return _series_view(f"{ax.root}/{group_of(ax.force)}", name, window,
                        contents=["$origin/**", "- $origin/prediction"])


def _events_view(origin: str, name: str, contents=None, entity_column: bool = False):
    """The event log: sample number, level, text (the text says the time; a time column is cut short)."""
    import rerun.blueprint as rrb
    from rerun.blueprint.encodings import TextLogColumn, TimelineColumn

    cols = rrb.TextLogColumns(
        timeline_columns=[TimelineColumn(SEQUENCE), TimelineColumn(TIMELINE, visible=False)],
        text_log_columns=[TextLogColumn("EntityPath", visible=entity_column), TextLogColumn("LogLevel"),
                          TextLogColumn("Body")])
    kw = {} if contents is None else {"contents": contents}
    return rrb.TextLogView(origin=origin, name=name, columns=cols, **kw)


def tooth_row(ax: AxisView, window: float | None):
    """The per-tooth panel (process monitors on): the last revolution's force over the spindle angle, its peak
    per tooth, and the once-per-revolution amplitude against the tooth monitor's limits."""
    import rerun.blueprint as rrb

    o = ax.root
    return rrb.Horizontal(
        rrb.BarChartView(origin=f"{o}/tooth/profile", name=f"{ax.axis}: measured force (N) over spindle angle (°), "
                         f"last {TOOTH_VIEW_REVOLUTIONS} revolutions", plot_legend=rrb.PlotLegend(visible=False)),
        rrb.BarChartView(origin=f"{o}/tooth/peaks",
                         name=f"peak force per tooth (N), last {TOOTH_VIEW_REVOLUTIONS} revolutions",
                         plot_legend=rrb.PlotLegend(visible=False)),
        _series_view(f"{o}/tooth", "per revolution (N): A1 and its limits (broken tooth red, runout orange), a0",
                     window, contents=["$origin/a0", "$origin/a1", "$origin/a1_broken", "$origin/a1_runout"]),
        column_shares=[1.4, 0.8, 1.8],
    )


def axis_blueprint(ax: AxisView, window: float | None = None, detail: float = 0.25):
    """One axis on one screen (after thesis Figure 4.8): disturbance and its detail, velocity, σ,
    dictionary, the two spectra with their markers (full width: a tick label every 10 Hz), events."""
    import rerun.blueprint as rrb

    o, u, g = ax.root, units_of(ax.force), group_of(ax.force)
    markers = f"{o}/psd_markers/**"
    key = "markers: 1/ψ yellow, tooth passing (and harmonics) cyan"
    what = "force" if ax.force else "disturbance"
    return rrb.Vertical(
        rrb.Horizontal(
            force_view(ax, window),
            _series_view(f"{o}/{g}", f"last {detail:g} s ({u}): one-step prediction orange, true green"
                                     f"{', dynamometer grey' if ax.force else ''}", detail, legend=None,
                         contents=["$origin/prediction", "$origin/actual", "$origin/dynamometer"]),
            column_shares=[2.2, 1],
        ),
        rrb.Horizontal(
            _series_view(f"{o}/velocity", f"{ax.axis} velocity (mm/s): reference, measured, one-step prediction",
                         window),
            _series_view(f"{o}/sigma", f"σ of the {what} estimate ({u})", window),
            _series_view(f"{o}/dictionary", "KRLS-T dictionary: size, pruning rate (1/s)", window),
            *([_series_view(f"{o}/context", "NC program line, tool number", window)] if ax.context else []),
            column_shares=[2, 1, 1] + ([1] if ax.context else []),
        ),
        rrb.BarChartView(origin=f"{o}/residual_psd", contents=["$origin/**", markers],
                         name=f"residual PSD (brown), dB above its floor, vs frequency (Hz); {key}",
                         plot_legend=rrb.PlotLegend(visible=False)),
        rrb.BarChartView(origin=f"{o}/disturbance_psd", contents=["$origin/**", markers],
                         name=f"{what} PSD, dB above its floor, vs frequency (Hz): estimate red, actual green; {key}",
                         plot_legend=rrb.PlotLegend(visible=False)),
        *([tooth_row(ax, window)] if ax.process and ax.force else []),
        _events_view(f"{o}/events", f"{ax.machine}/{ax.axis} events: flags, gaps, glitches, health"
                                    f"{', process alarms' if ax.process else ''}"),
        # with the per-tooth row the spectra give it room (bar charts need height for their tick labels)
        row_shares=[2.4, 1.5, 1.85, 1.85, 1.9] if not (ax.process and ax.force) else [2.3, 1.4, 1.3, 1.3, 2.4, 1.6],
        name=f"{ax.machine}/{ax.axis}",
    )


def overview(axes: Sequence[AxisView], window: float | None):
    """Several axes: one disturbance panel per axis and the events of all axes."""
    import rerun.blueprint as rrb

    panels = [force_view(ax, window, title_prefix=f"{ax.machine}/") for ax in axes]
    log = _events_view("/", "events of all axes", contents=[f"{ax.root}/events" for ax in axes], entity_column=True)
    return rrb.Vertical(*panels, log, row_shares=[2] * len(panels) + [1], name="overview")


def blueprint_for(axes: Sequence[AxisView], window: float | None = None, detail: float = 0.25):
    """The dashboard: one axis on its own, else an overview tab and one tab per axis.

    ``window``: rolling window (s of controller time) of the time views, None = the whole run.
    """
    import rerun.blueprint as rrb

    views = [axis_blueprint(ax, window, detail) for ax in axes]
    if not views:
        root = rrb.Vertical(rrb.TextDocumentView(origin="/", name="waiting for data"))
    elif len(views) == 1:
        root = views[0]
    else:
        root = rrb.Tabs(overview(axes, window), *views)
    return rrb.Blueprint(root, rrb.BlueprintPanel(state="hidden"), rrb.SelectionPanel(state="hidden"),
                         rrb.TimePanel(state="collapsed", timeline=TIMELINE, play_state="following"))
