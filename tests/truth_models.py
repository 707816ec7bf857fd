"""Simulated trials and model files with the simulator's TRUE β (one definition for the service tests)."""

from __future__ import annotations

from pathlib import Path

from feedio.mcapio import read_trial
from monitor.model_file import save_model, truth_model
from replay.scenarios import load_scenario
from replay.simulator import simulate, write_trial


def make_trial(path: Path, duration: float, seed: int, scenario: str = "shaker-constant") -> Path:
    """A simulated trial of ``duration`` s written to ``path``."""
    write_trial(simulate(load_scenario(scenario, duration=duration), seed=seed), path)
    return path


def model_from_truth(trial: Path, path: Path, *, period: float = 1 / 55, budget: int = 50) -> Path:
    """Model file with the trial's TRUE β and the thesis tracker hyperparameters (Table 4.5)."""
    return save_model(truth_model(read_trial(trial).meta, period=period, budget=budget), path)


def truth_workdir(tmp_path_factory, name: str, *, duration: float, seed: int, budget: int = 50) -> Path:
    """A fresh folder holding ``trial.mcap`` (shaker, ``duration`` s) and ``z.model.toml`` (its truth)."""
    d = tmp_path_factory.mktemp(name)
    make_trial(d / "trial.mcap", duration, seed)
    model_from_truth(d / "trial.mcap", d / "z.model.toml", budget=budget)
    return d
