"""Imported by the batch's forkserver (:mod:`rig.catalog.batch`, ``START_METHOD``) after the task's module:
numba's CPU target is loaded here once (its typing and lowering registries: about 0.3 s of CPU), so every
worker forked from the server starts with it, instead of paying it at its first task (measured: a worker's
first identify-kernel call took 0.37 s of CPU without it, 0.02 s with it; docs/scaling.md). The kernels'
own cached machine code (a few ms each) is still loaded where it is first called."""

from numba.core.registry import cpu_target

cpu_target.target_context.refresh()
