"""Controller bridges: a machine's servo-rate data → feedmon's sample blocks on Zenoh, and the
monitor's findings back to the machine. One sub-package per controller (:mod:`bridge.linuxcnc`).

A bridge imports ``feedio`` (the schema, Zenoh keys and sessions, trial files) and nothing above it.
"""
