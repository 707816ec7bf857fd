"""The ``[monitors]`` table of the ``feedmon run`` configuration: one msgspec Struct per monitor.

Every number has its allowed range in its type (decoding a config file checks it and the error names
the key and the range); ``sensitivity`` is the ``k`` of the monitor's ``k·σ`` limits (larger: fewer
alarms). Units: N, s, revolutions, parts.
"""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from feedio.schema import PROFILE_BINS_MAX, TEETH_MAX

__all__ = ["ImpulseSettings", "ToothSettings", "EnvelopeSettings", "WearSettings", "SectionLimits",
           "MonitorSettings", "MAX_SECTIONS", "MAX_KEEP"]

#: the most ``[[monitors.section]]`` entries a configuration may hold
MAX_SECTIONS = 1000

_Newton = Annotated[float, msgspec.Meta(ge=0.0, le=1e7)]
_K = Annotated[float, msgspec.Meta(ge=1.0, le=100.0)]


class ImpulseSettings(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Collision (impulse beyond the expected force) and overload (``|F|`` above ``overload_N``)."""

    enabled: bool = True
    #: the force judged: "filtered" (the tracker's estimate) or "measured" (the one-step residual in N)
    signal: Literal["filtered", "measured"] = "measured"
    limit_N: _Newton = 50.0  # floor of the collision limit (N): below it no impulse is a collision
    ratio: Annotated[float, msgspec.Meta(ge=1.0, le=100.0)] = 1.5  # × running peak |F| (no spindle angle)
    ratio_angle: Annotated[float, msgspec.Meta(ge=0.1, le=100.0)] = 1.0  # × max |profile| (with spindle angle)
    sensitivity: _K = 6.0
    window_s: Annotated[float, msgspec.Meta(ge=0.006, le=10.0)] = 0.1  # running peak and hold-off after an alarm
    bins: Annotated[int, msgspec.Meta(ge=4, le=720)] = 12  # angle bins of the expected force
    alpha: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)] = 0.5  # weight of a new sample in its bin
    overload_N: Annotated[float, msgspec.Meta(gt=0.0, le=1e7)] | None = None  # None: no overload monitor
    persist: Annotated[int, msgspec.Meta(ge=1, le=10_000)] = 3  # overload: samples in a row


class ToothSettings(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Per tooth from the spindle angle: broken/chipped tooth and runout growth."""

    enabled: bool = True
    teeth: Annotated[int, msgspec.Meta(ge=1, le=TEETH_MAX)] = 2
    bins: Annotated[int, msgspec.Meta(ge=4, le=PROFILE_BINS_MAX)] = 36  # angle profile (dashboard, per-tooth peaks)
    learn_revolutions: Annotated[int, msgspec.Meta(ge=5, le=100_000)] = 30
    settle_revolutions: Annotated[int, msgspec.Meta(ge=0, le=100_000)] = 25  # of a cut's entry, before learning
    sensitivity: _K = 6.0
    cut_min_N: _Newton = 5.0  # a revolution with a mean force below this is no cut
    broken_fraction: Annotated[float, msgspec.Meta(gt=0.0, le=10.0)] = 0.5  # of the mean cutting force
    runout_fraction: Annotated[float, msgspec.Meta(gt=0.0, le=10.0)] = 0.1


class EnvelopeSettings(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Against a reference learned from good runs (``feedmon reference learn``): missing cut, over band."""

    reference: Annotated[list[str], msgspec.Meta(max_length=1024)] = []  # reference files (one per axis); none: off
    sensitivity: _K = 5.0
    band_min_N: _Newton = 5.0
    persist_s: Annotated[float, msgspec.Meta(ge=0.0, le=60.0)] = 0.1
    cut_min_N: _Newton = 5.0  # a reference bin with a mean below this expects no cut


#: the most parts a wear history keeps per section (``keep``)
MAX_KEEP = 200


class WearSettings(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Wear trend across parts (M7): one history file of per-section statistics, judged at the end of each run.

    Alarm ⇔ over the last ``window`` parts (at least ``min_parts``) the slope's t statistic exceeds
    ``sensitivity`` and the fitted rise exceeds ``min_rise`` of the fitted first value. Why these defaults
    (false-alarm probability per part and over 200 parts): ``docs/process-monitoring.md``, "Wear"."""

    history: Annotated[str, msgspec.Meta(min_length=1, max_length=4096)] | None = None  # None: no wear monitor
    statistic: Literal["mean_force", "energy"] = "mean_force"  # |mean force| (N) or |cut energy ∫F·v dt| (J)
    window: Annotated[int, msgspec.Meta(ge=3, le=MAX_KEEP)] = 20  # parts the trend is fitted over
    min_parts: Annotated[int, msgspec.Meta(ge=3, le=MAX_KEEP)] = 10  # parts a section needs before it is judged
    keep: Annotated[int, msgspec.Meta(ge=3, le=MAX_KEEP)] = 50  # parts kept per section in the file
    sensitivity: _K = 5.0  # the t statistic's limit
    min_rise: Annotated[float, msgspec.Meta(gt=0.0, le=10.0)] = 0.10  # fitted rise over the window, relative
    cut_min_N: _Newton = 5.0  # a section whose |mean force| is below this is no cut: not recorded

    def __post_init__(self) -> None:
        if not self.min_parts <= self.window <= self.keep:
            raise ValueError(f"min_parts ({self.min_parts}) ≤ window ({self.window}) ≤ keep ({self.keep}) is needed")


class SectionLimits(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Absolute limits of one tool and/or NC line (``[[monitors.section]]``); a row matches when every given
    key equals its context."""

    tool: Annotated[int, msgspec.Meta(ge=-(2**31), le=2**31 - 1)] | None = None
    program_line: Annotated[int, msgspec.Meta(ge=-(2**31), le=2**31 - 1)] | None = None
    limit_N: _Newton | None = None
    overload_N: Annotated[float, msgspec.Meta(gt=0.0, le=1e7)] | None = None


class MonitorSettings(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """The ``[monitors]`` table. ``enabled`` false (the default): no process monitor runs, outputs unchanged."""

    enabled: bool = False
    impulse: ImpulseSettings = ImpulseSettings()
    tooth: ToothSettings = ToothSettings()
    envelope: EnvelopeSettings = EnvelopeSettings()
    wear: WearSettings = WearSettings()
    section: Annotated[list[SectionLimits], msgspec.Meta(max_length=MAX_SECTIONS)] = []
    ack_widen: Annotated[float, msgspec.Meta(ge=1.0, le=10.0)] = 1.5  # each acknowledged false alarm widens ×
