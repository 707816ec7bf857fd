"""Offline identification of one axis: candidate models, chosen by evidence among the valid ones
(docs/method.md §8).

:func:`identify` takes a :class:`feedio.mcapio.Trial` and returns an :class:`Identification`. The
package, top to bottom (imports point down only):

* :mod:`.workflow` — :func:`identify`, step by step;
* :mod:`.regression` — the regression all candidates share: dead band, friction and process columns;
* :mod:`.periods` — the periods in play and the kernel candidates tuned at them;
* :mod:`.truth` — errors against a simulated or published truth;
* :mod:`.result` — :class:`Identification`: the JSON document and the model file;
* :mod:`.rules` — validity rules 2 and 3, the choice;
* :mod:`.candidates` — the regression shared by all candidates, a candidate, its fit, the constants.
"""

from kernels.feed_drive import COULOMB_Z

from ..online_settings import TRACKER_DEFAULTS
from .candidates import (
    EFFICIENCY_KEYS,
    SUGGEST_MARGIN,
    THESIS_DEFAULTS,
    UNDETERMINED_RSE,
    VIF_FLAG,
    Candidate,
    MethodResult,
)
from .periods import periods_in_play
from .regression import dead_band
from .result import Identification
from .workflow import identify

__all__ = ["THESIS_DEFAULTS", "TRACKER_DEFAULTS", "UNDETERMINED_RSE", "EFFICIENCY_KEYS",
           "VIF_FLAG", "SUGGEST_MARGIN", "COULOMB_Z", "Identification", "Candidate", "MethodResult", "identify",
           "periods_in_play", "dead_band"]
