"""The HAL side of ``feedmon bridge linuxcnc``: read one ``sampler`` FIFO, own the way-back pins.

Runs under the Python that LinuxCNC's ``hal`` module is built for (Debian: ``/usr/bin/python3``),
as a child of the bridge, which may run under any Python (its venv): this file imports only the
standard library and ``hal``, never feedmon. The bridge starts it with the JSON spec as the one
argument (see :func:`main`) and talks to it through pipes:

* stdout, frames ``<u32 length><u8 kind><payload>`` (little endian): ``H`` hello (JSON: the FIFO's
  column types, depth, overruns, the samples it held when attached — written while nobody read them,
  discarded —, the HAL session id, the helper's pid), ``D`` data (``<d I I I``: CLOCK_MONOTONIC of
  the read in s, the FIFO's overrun count, rows, columns; then rows × columns float64 — u32, s32 and
  bit columns are exact as float64), ``E`` error (JSON ``{"error": …}``, then the helper exits);
* stdin, one JSON object per line: ``{"<pin>": value, …}`` sets those pins of the component.

HAL streams have no blocking read, so the FIFO is polled every ``poll`` seconds (the wait is a
``select`` on stdin: pin updates are applied as soon as they arrive). The helper ends at EOF on
stdin (the bridge ended), at SIGTERM/SIGINT (LinuxCNC's ``halcmd unload all`` at shutdown), and
when the sampler's FIFO leaves shared memory (HAL stopped): always through ``component.exit()``,
which removes its pins from HAL.

It never creates a HAL session: the sampler's FIFO must be in shared memory before
``hal.component`` is called (otherwise ``hal`` would start an empty HAL of its own).
"""

import json
import os
import select
import signal
import struct
import sys
import time

HAL_KEY = 0x48414C32  # the HAL shared memory segment ("HAL2"); its shmid identifies the HAL session
TYPE_CODES = {"float": "HAL_FLOAT", "bit": "HAL_BIT", "s32": "HAL_S32", "u32": "HAL_U32"}
#: the head of a ``D`` frame: read time (s, CLOCK_MONOTONIC), FIFO overruns, rows, columns (the helper reads it)
DATA_HEAD = struct.Struct("<dIII")


def shm_ids():
    """``{key: shmid}`` of the System V shared memory segments (``/proc/sysvipc/shm``)."""
    out = {}
    with open("/proc/sysvipc/shm") as f:
        next(f)
        for line in f:
            parts = line.split()
            if len(parts) > 1:
                out[int(parts[0])] = int(parts[1])
    return out


def frame(kind, payload):
    out = sys.stdout.buffer
    out.write(struct.pack("<IB", len(payload), ord(kind)) + payload)
    out.flush()


def fail(message, code=2):
    frame("E", json.dumps({"error": message}).encode())
    sys.exit(code)


def make_component(hal, spec):
    """The way-back component: its output pins, linked to the signals the spec names."""
    name = spec["component"]
    try:
        comp = hal.component(name)
    except Exception as exc:  # noqa: BLE001 - hal_init's failure
        fail(f"cannot create the HAL component {name} ({exc}): is there one of that name already (another bridge, "
             f"or one killed without leaving HAL: halcmd unload {name})? Or set [hal] component to another name")
    try:
        _pins_and_links(hal, comp, spec)
    except BaseException:
        comp.exit()
        raise
    return comp


def _pins_and_links(hal, comp, spec):
    for name, kind in spec["pins"]:
        comp.newpin(name, getattr(hal, TYPE_CODES[kind]), hal.HAL_OUT)
    comp.ready()
    signals = {s["NAME"]: s for s in hal.get_info_signals()}
    for pin, sig in spec.get("links", {}).items():
        full = f"{spec['component']}.{pin}"
        if sig in signals and signals[sig]["DRIVER"] not in (None, "", full):
            fail(f"signal {sig} already has a writer ({signals[sig]['DRIVER']}); the bridge's pin {full} cannot "
                 "drive it: remove that writer or link the pin to another signal")
        try:
            if sig not in signals:
                hal.new_sig(sig, getattr(hal, TYPE_CODES[dict(spec["pins"])[pin]]))
            hal.connect(full, sig)
        except Exception as exc:  # noqa: BLE001 - hal raises RuntimeError/ValueError/TypeError
            fail(f"cannot link {full} to signal {sig}: {exc} (a signal of another type?)")


def main(argv):
    spec = json.loads(argv[1])
    stop = []
    key = None
    try:
        import hal
        key = hal.sampler_base + int(spec["sampler"])
    except ImportError as exc:
        fail(f"{sys.executable} cannot import LinuxCNC's hal module ({exc}); give the Python it is built for "
             "(Debian: /usr/bin/python3) or install LinuxCNC (apt-get install linuxcnc-uspace)", 3)
    ids = shm_ids()
    if key not in ids or HAL_KEY not in ids:
        fail(f"sampler.{spec['sampler']} has no FIFO in shared memory: HAL is not running, or its HAL file has no "
             f"'loadrt sampler' with channel {spec['sampler']}", 4)
    session, fifo = ids[HAL_KEY], ids[key]
    comp = make_component(hal, spec)
    for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGPIPE):  # after hal.component, which sets its own
        signal.signal(sig, lambda *_: stop.append(1))
    try:
        try:
            stream = hal.stream(comp, key)
        except Exception as exc:  # noqa: BLE001
            fail(f"cannot attach to the FIFO of sampler.{spec['sampler']}: {exc}", 4)
        types = stream.element_types.decode() if isinstance(stream.element_types, bytes) else str(stream.element_types)
        stale = 0
        while stale < 10 * stream.maxdepth and stream.read() is not None:  # written while nobody listened
            stale += 1
        frame("H", json.dumps({"types": types, "maxdepth": stream.maxdepth, "overruns": stream.num_overruns,
                               "stale": stale, "session": session, "pid": os.getpid()}).encode())
        loop(hal, comp, stream, spec, stop, key, fifo)
    finally:
        comp.exit()


def loop(hal, comp, stream, spec, stop, key, fifo):
    poll, max_rows = float(spec.get("poll", 0.0005)), int(spec.get("max_rows", 4096))
    ncol = len(stream.element_types)
    read, stdin = stream.read, sys.stdin.buffer
    pending = b""
    next_check = time.monotonic() + 1.0
    while not stop:
        ready, _, _ = select.select([stdin], [], [], poll)
        if ready:
            chunk = os.read(stdin.fileno(), 65536)
            if not chunk:
                return  # the bridge ended
            *lines, pending = (pending + chunk).split(b"\n")
            for line in lines:
                for pin, value in json.loads(line).items():
                    comp[pin] = value
        rows = []
        while len(rows) < max_rows:
            row = read()
            if row is None:
                break
            rows.append(row)
        if rows:
            flat = [float(x) for row in rows for x in row]
            frame("D", DATA_HEAD.pack(time.monotonic(), stream.num_overruns, len(rows), ncol)
                  + struct.pack(f"<{len(flat)}d", *flat))
        now = time.monotonic()
        if now >= next_check:
            next_check = now + 1.0
            if shm_ids().get(key) != fifo:
                fail("HAL stopped: the sampler's FIFO left shared memory", 5)


if __name__ == "__main__":
    try:
        main(sys.argv)
    except (BrokenPipeError, KeyboardInterrupt):
        pass
