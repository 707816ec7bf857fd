"""The LinuxCNC bridge (``feedmon bridge linuxcnc``), in both directions.

* in: a HAL ``sampler`` FIFO, read by a helper under the Python LinuxCNC's ``hal`` module is built
  for (:mod:`.helper`, :mod:`.halio`); its columns mapped to :class:`~feedio.schema.SampleBlock`
  columns as the configuration says (:mod:`.config`, checked against HAL's wiring by :mod:`.wiring`;
  :mod:`.mapper`); published on Zenoh and/or written to a trial file (:mod:`.run`);
* back: the monitor's estimates and alarms → output pins of the helper's HAL component, which the
  user wires, e.g. to ``motion.feed-hold`` (:mod:`.wayback`).

How to connect a machine: ``docs/linuxcnc.md``.
"""
