"""A model whose force acts d samples late ([model] delay): the monitor's first regressor is the batch fit's."""

import numpy as np
import pytest

from feedio.mcapio import iter_blocks, read_trial
from kernels.feed_drive import regressors
from monitor.estimator import AxisEstimator
from monitor.identify import identify


@pytest.fixture(scope="module")
def delayed(simulated):
    """A command-delay drive identified on one trial (no options) and another trial of it to monitor."""
    result = identify(read_trial(simulated("command-delay", seed=1, duration=12.0)))
    return result.to_model(feedmon_version="test"), simulated("command-delay", seed=2, duration=12.0)


def test_the_delayed_command_is_the_batch_regressor_across_blocks(delayed):
    """Block by block, the carried history gives exactly the batch regressor's first column (its first d rows
    excepted: the batch and the monitor both keep the undelayed command where no past exists)."""
    model, path = delayed
    assert model.delay >= 1
    est = AxisEstimator(model)
    trial = read_trial(path)
    got = []
    for _, b in iter_blocks(path, kinds=("samples",)):
        e = np.asarray(b.u if model.form == "force-input" else b.v_ref, dtype=float)
        got.append(est._delayed_command(int(b.seq), e, np.asarray(b.v_meas, dtype=float)))
    got = np.concatenate(got)
    want = regressors(model.form, trial.v_meas, v_ref=trial.v_ref, u=trial.u, omega=model.omega,
                      delay=model.delay).Z[:, 0]
    np.testing.assert_allclose(got[model.delay:want.size], want[model.delay:], rtol=0, atol=1e-12)  # Z: one row less


def test_out_of_sample_force_with_and_without_the_delay(delayed):
    """Out of sample (model from seed 1, trial seed 2): with the delay the one-step force prediction follows the
    truth (corr 0.94); the same β without it (the monitor before it knew delays) is clearly worse (0.75)."""
    from dataclasses import replace

    model, path = delayed
    trial = read_trial(path)

    def corr(m):
        est = AxisEstimator(m)
        f = [est.process(b).force_next for _, b in iter_blocks(path, kinds=("samples",))]
        f = np.concatenate(f)
        keep = np.arange(f.size) > 3 * 333
        ok = keep & np.isfinite(f)
        return np.corrcoef(f[ok], trial.truth.force[ok])[0, 1]

    with_delay, without = corr(model), corr(replace(model, delay=0))
    assert with_delay > 0.9, (with_delay, without)
    assert with_delay > without + 0.1, (with_delay, without)
