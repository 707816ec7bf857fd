"""The feedmon service: identification workflow, model files, the per-axis estimator, the live
monitor and its sinks. Uses :mod:`kernels` and :mod:`feedio`; never imports :mod:`replay` or the CLI."""
