"""Measurement helpers shared by the bench scripts (Linux /proc; no dependencies).

Bench scripts run as ``python bench/NAME.py``, so this folder is on sys.path.
"""

from __future__ import annotations

import os
import time

CLK_TCK = os.sysconf("SC_CLK_TCK")


def machine_busy_s() -> float:
    """CPU seconds all cores spent not idle since boot (/proc/stat, minus idle and iowait)."""
    with open("/proc/stat") as f:
        values = [int(v) for v in f.readline().split()[1:]]
    return (sum(values[:8]) - values[3] - values[4]) / CLK_TCK


def proc_cpu_s(pid: int | str = "self") -> float:
    """utime + stime of a process (or "PID/task/TID" for a thread), seconds.

    Raises FileNotFoundError/ProcessLookupError when it is gone.
    """
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def wait_idle(max_wait: float, threshold: float, sample: float = 2.0) -> float:
    """Wait (at most ``max_wait`` s) until the machine's busy CPU over ``sample`` s is below
    ``threshold`` of one core; returns the last busy fraction seen."""
    deadline = time.monotonic() + max_wait
    while True:
        a = machine_busy_s()
        time.sleep(sample)
        busy = (machine_busy_s() - a) / sample
        if busy < threshold or time.monotonic() >= deadline:
            return busy


def exact_ring_rig(poses):
    """A rig that knows every virtual sensor's true pose: ids s0, s1, ... for ``poses``
    (``VirtualPose``s, e.g. ``ring_poses``), s0 the reference and stage space."""
    from stage.geometry import invert
    from stage.rig import Rig, set_calibration
    rig = Rig(reference="s0")
    rig.stage_frame = poses[0].to_stage
    for k, p in enumerate(poses):
        set_calibration(rig, f"s{k}", invert(poses[0].to_stage) @ p.to_stage, "bench")
    return rig
