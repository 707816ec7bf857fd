"""The monitored axes: model file → :class:`AxisRuntime` (model, estimator, status), and the MCAP
metadata of a monitored axis (the warm-up before "ready": :mod:`monitor.warm`)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from feedio import schema as S
from kernels.errors import ParameterError

from .estimator import AxisEstimator
from .model_file import AxisModel, file_sha256, load_model
from .online_settings import apply_overrides
from .status import AxisStatus

__all__ = ["AxisRuntime", "load_axes", "live_meta"]


@dataclass
class AxisRuntime:
    """One monitored axis: its model, estimator and status."""

    model: AxisModel
    estimator: AxisEstimator
    status: AxisStatus

    @property
    def key(self) -> tuple[str, str]:
        return (self.model.machine, self.model.axis)


def load_axes(model_paths: Sequence[str | os.PathLike], config=None) -> dict[tuple[str, str], AxisRuntime]:
    """Load model files (one per axis); two files for the same axis, or a machine/axis name the
    message schema does not allow (:data:`feedio.limits.NAME_PATTERN`), are errors. ``config`` (a
    :class:`feedmon.run_config.RunConfig`): its ``tracker``/``adaptation``/``health`` overrides
    replace the model files' settings (:func:`monitor.online_settings.apply_overrides`)."""
    if not model_paths:
        raise ParameterError("model_paths is empty: give at least one model file", "model_paths")
    axes: dict[tuple[str, str], AxisRuntime] = {}
    for p in model_paths:
        path = Path(p)
        model = load_model(path)
        if config is not None:
            try:
                model = apply_overrides(model, config.tracker, config.adaptation, config.health)
            except ValueError as exc:
                raise ParameterError(f"model file {path}, with the overrides of config: {exc}", "config") from None
        for what in ("machine", "axis"):  # the names a message must carry (feedio.schema): else no block could match
            try:
                S.check_name(getattr(model, what), f"model {what}")
            except ValueError as exc:
                raise ValueError(f"model file {path}: {exc}") from None
        key = (model.machine, model.axis)
        if key in axes:
            raise ValueError(f"two model files for axis {model.machine}/{model.axis}: "
                             f"{axes[key].status.model_path} and {path}")
        st = AxisStatus(model.machine, model.axis, str(path), file_sha256(path))
        axes[key] = AxisRuntime(model, AxisEstimator(model), st)
    return axes


def live_meta(ax: AxisRuntime, source: str = "live") -> S.TrialMeta:
    """TrialMeta of a monitored axis for the MCAP log (Ts and form from the model file)."""
    from feedio import __version__

    m = ax.model
    return S.TrialMeta(
        Ts=float(m.Ts), form=m.form, machine=m.machine, axis=m.axis, loop_gain=m.loop_gain,
        units=dict(S.UNITS),
        provenance=S.Provenance(source=source, tool="feedmon run", version=__version__,
                                details={"model_file": ax.status.model_path, "model_sha256": ax.status.model_sha256,
                                         "tracker_state": ax.status.state}),
        description="feedmon monitor log: input samples and disturbance estimates",
    )
