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


#: the test files that take longest, handed to the workers first: pytest-xdist gives each worker whole files in
#: collection order, and a long file begun last leaves the other worker idle at the end (longest first)
LONG_FIRST = ("test_deploy.py", "test_identify.py", "test_linuxcnc.py", "test_soak.py", "test_out_of_sample.py",
              "test_sink_faults.py", "test_fast_paths.py", "test_krlst.py", "test_online_health.py", "test_faults.py",
              "test_run_e2e.py", "test_state.py", "test_dashboard.py", "test_adequacy.py")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONG_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(LONG_FIRST)))  # stable: the others keep their order
