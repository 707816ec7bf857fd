"""Shared test fixtures: the real EMPS recordings and simulated trials (made once per session)."""

import os
from pathlib import Path

import pytest

from feedmon.cli import main
from replay.importers import EMPS_HOWTO

REPO = Path(__file__).resolve().parents[1]


def _emps_path(name: str) -> Path:
    folder = Path(os.environ.get("FEEDMON_EMPS_DIR", REPO / ".." / "shared" / "data" / "emps"))
    path = folder / name
    if not path.is_file():
        pytest.fail(f"EMPS file {path} not found (set FEEDMON_EMPS_DIR): {EMPS_HOWTO}", pytrace=False)
    return path


@pytest.fixture(scope="session")
def emps_file():
    """``emps_file("DATA_EMPS.mat")`` → path; fails (never skips) with how to get the data."""
    return _emps_path


@pytest.fixture(scope="session")
def simulated(tmp_path_factory):
    """``simulated("shaker-constant", seed=1)`` → path of a trial made by ``feedmon simulate`` (cached)."""
    cache: dict = {}
    folder = tmp_path_factory.mktemp("trials")

    def make(scenario: str, seed: int = 1, duration: float | None = None) -> Path:
        key = (scenario, seed, duration)
        if key not in cache:
            out = folder / f"{scenario}-{seed}-{duration}.mcap"
            argv = ["simulate", scenario, "-o", str(out), "--seed", str(seed)]
            if duration is not None:
                argv += ["--duration", str(duration)]
            assert main(argv) == 0
            cache[key] = out
        return cache[key]

    return make

