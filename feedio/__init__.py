"""Shared I/O of feedmon, below both the service (``monitor``) and the trials (``replay``):

* :mod:`feedio.schema` — the one message schema (samples, truth, estimates, trial metadata);
* :mod:`feedio.mcapio` — MCAP trial and log files (one writer, one reader);
* :mod:`feedio.mcapfile` — checked, bounded MCAP record parsing (limits, CRCs) under the reader and recover;
* :mod:`feedio.scalars` — the per-sample ``disturbance/scalars`` messages (pairing rows and truth in time);
* :mod:`feedio.transport` — Zenoh sessions and key expressions;
* :mod:`feedio.digest` — file digests for provenance.

Dependencies run one way: ``kernels`` (numerics) ← ``feedio`` ← ``monitor``, ``replay`` ← ``feedmon`` (CLI).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("feedmon")
except PackageNotFoundError:  # running from a source tree without install
    __version__ = "0.0.0+unknown"
