"""Trials: simulated feed-drive trials with known truth, importers, and MCAP replay over Zenoh."""
