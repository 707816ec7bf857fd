"""The warm-up before "ready" (:mod:`monitor.warm`) reaches every compiled function the live path uses.

Checked in a fresh interpreter (a test worker has compiled everything already): after ``warm_up``, two
axes — a milling axis with spindle data and a shaker axis without — run a simulated trial each through
the pipeline with the process monitors on, the disturbance search adopting models, and a state save; no
compiled function of ``kernels`` gains a compiled signature meanwhile. A function first met there would
be compiled (seconds on a cold cache) while samples and alarms wait.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = r"""
import json, sys, tempfile
from pathlib import Path
from numba.core.dispatcher import Dispatcher

def signatures():
    out = {}
    for name, mod in list(sys.modules.items()):
        if not name.startswith("kernels"):
            continue
        for attr, obj in vars(mod).items():
            if isinstance(obj, Dispatcher):
                out[f"{obj.py_func.__module__}.{obj.py_func.__qualname__}"] = len(obj.overloads)
    return out

from feedio import schema as S
from monitor.axes import load_axes
from monitor.model_file import save_model, truth_model
from monitor.pipeline import Pipeline
from monitor.process_monitor import build_monitors
from monitor.process_monitor.settings import MonitorSettings
from monitor.state import StateStore
from monitor.warm import warm_up
from replay.scenarios import load_scenario
from replay.simulator import simulate

work = Path(tempfile.mkdtemp())
trials, paths = {}, []
for name, period in (("milling-incdec", 1 / 100), ("shaker-constant", 1 / 13)):
    tr = simulate(load_scenario(name, duration=12.0), seed=11)
    tr.meta.axis = name.split("-")[0]
    path = work / f"{name}.model.toml"
    save_model(truth_model(tr.meta, period=period, budget=60), path)
    trials[(tr.meta.machine, tr.meta.axis)] = tr
    paths.append(path)
axes = load_axes(paths)
monitors = build_monitors(axes, MonitorSettings(enabled=True))
warm_up(axes, monitors)
before = signatures()

pipe = Pipeline(axes, monitors=monitors)
for key, tr in trials.items():
    for i in range(0, tr.t.size, 7):
        sl = slice(i, i + 7)
        extra = {}
        if tr.spindle_angle is not None:
            extra = dict(spindle_angle=tr.spindle_angle[sl].tolist(), spindle_rpm=tr.spindle_rpm[sl].tolist())
        block = S.SampleBlock(machine=key[0], axis=key[1], seq=i, t=tr.t[sl].tolist(), v_ref=tr.v_ref[sl].tolist(),
                              v_meas=tr.v_meas[sl].tolist(), **extra)
        pipe.estimate(block)
store = StateStore(work / "state")
for ax in axes.values():
    store.save(ax)
after = signatures()
print(json.dumps({
    "new": sorted(k for k, n in after.items() if n > before.get(k, 0)),
    "functions": len(before),
    "searches": {"/".join(k): ax.estimator.counters["tracker_searches"] for k, ax in axes.items()},
    "adoptions": {"/".join(k): ax.estimator.counters["tracker_adoptions"] for k, ax in axes.items()},
}))
"""


def test_warm_up_leaves_nothing_to_compile(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, "-c", SCRIPT], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=900)
    assert proc.returncode == 0, proc.stderr[-4000:]
    doc = json.loads(proc.stdout.strip().splitlines()[-1])
    assert doc["functions"] > 30, doc                        # the kernels' compiled functions were seen
    assert all(n > 0 for n in doc["adoptions"].values()), doc  # the search adopted on both axes
    assert doc["new"] == [], f"compiled after the warm-up: {doc['new']}"


COMPILE_ALL = r"""
import json, sys
from numba.core.dispatcher import Dispatcher
from monitor.warm import compile_all
compile_all()
seen = {}
for name, mod in list(sys.modules.items()):
    if name.startswith("kernels"):
        for obj in vars(mod).values():
            if isinstance(obj, Dispatcher):
                seen[f"{obj.py_func.__module__}.{obj.py_func.__qualname__}"] = len(obj.overloads)
print(json.dumps(seen))
"""


def test_the_image_build_step_loads_what_the_first_search_and_alarm_need(tmp_path):
    """``compile_all`` (the Dockerfile's build step, no model file) leaves in a fresh interpreter the
    compiled versions the live path meets late: the search's replays, online β's rebase, the tracker API an adoption calls, the monitors' cores."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, "-c", COMPILE_ALL], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-4000:]
    seen = json.loads(proc.stdout.strip().splitlines()[-1])
    for name in ("kernels._krlst_core.track", "kernels.beta_step.replay_joint", "kernels._krlst_core.update_buffers",
                 "kernels._krlst_core.arm_buffers", "kernels._krlst_core.learn_buffers",
                 "kernels.online.track_block", "kernels.force_monitors.impulse_step",
                 "kernels.force_monitors.tooth_block", "kernels.period._harmonic_sum"):
        assert seen.get(name, 0) >= 1, name
