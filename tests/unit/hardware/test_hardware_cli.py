"""`rig devices check` and `rig loop-bench` through the CLI."""

from __future__ import annotations


def test_skipped_cycles_are_attributed_to_the_vm_or_the_loop():
    from rig.hardware.timing import attribute_skips

    gaps = [(10.0, 10.03)]  # the probe slept 30 ms over there
    skips = [(10.031, 25), (20.004, 3)]  # one late tick inside the probe's stall, one on its own
    a = attribute_skips(skips, gaps, 1e-3)
    assert (a["vm_cycles"], a["loop_cycles"], a["vm_episodes"], a["loop_episodes"]) == (25, 3, 1, 1)
    assert a["loop_at"] == [(20.004, 3)]
