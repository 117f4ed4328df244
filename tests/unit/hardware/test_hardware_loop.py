"""The trial session on the hardware backend against the emulated rig: a clean run, and
interlock trips that end in the safe state (valve nulled and disabled, seen from the valve
emulator), with the session's stop state machine reaching SAFE then DONE."""

from __future__ import annotations

import pytest


@pytest.mark.parametrize("late_periods", [0.3, 1.4, 2.5, 7.9, 100.2])
def test_a_late_wake_skips_what_due_skips_says(late_periods):
    """The stall event's skipped count: a tick that wakes late has ``due_skips(wake)`` deadlines behind it
    already; advance() at the end of that tick skips exactly those (plus what a long tick adds)."""
    from rig.hardware.timing import Pacer

    p = Pacer(1e-3, fifo=True)
    p.start(t0=10.0)
    for _ in range(5):
        p.advance(p.deadline() + 1e-4)
    wake = p.deadline() + late_periods * 1e-3
    due = p.due_skips(wake)
    assert due == (0 if late_periods < 2.0 else int(late_periods))
    assert p.advance(wake) == due and p.skipped == due
    assert p.advance(p.deadline() + 2.6e-3) >= 2  # a long tick: skips counted by advance, not due at wake
