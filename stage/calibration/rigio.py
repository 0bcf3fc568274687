"""Writing calibration results into a rig (the installer's YAML)."""

from __future__ import annotations

import numpy as np

from ..rig import Rig, SensorConfig, set_calibration
from ..geometry import invert


def store_stage_transform(rig: Rig, sensor: str, to_stage: np.ndarray, reference: str | None,
                          method: str, fitness: float | None, rms_m: float | None) -> None:
    """Record a sensor -> STAGE transform (what the engine uses) in the rig.

    The rig keeps each sensor's transform into the reference sensor's space
    and the reference's own placement as ``stage_frame``. A new transform for
    the reference itself (it was moved and re-calibrated against the others)
    becomes the new stage frame, and every other calibration is re-expressed
    against it, so stage space stays where the other sensors put it.
    """
    if reference is not None:
        rig.reference = reference
        rig.sensors.setdefault(reference, SensorConfig(reference))
    if sensor == rig.reference:
        old = rig.stage_frame
        new_inverse = invert(to_stage)
        for sid, config in rig.sensors.items():
            if sid != sensor and config.calibration is not None:
                config.calibration.matrix = new_inverse @ old @ config.calibration.matrix
        rig.stage_frame = np.asarray(to_stage, dtype=float)
        set_calibration(rig, sensor, np.eye(4), method, fitness, rms_m)
    else:
        set_calibration(rig, sensor, invert(rig.stage_frame) @ to_stage, method, fitness, rms_m)


def store_reference_transform(rig: Rig, sensor: str, to_reference: np.ndarray,
                              reference: str, method: str, fitness: float | None,
                              rms_m: float | None) -> None:
    """Record a sensor -> REFERENCE-space transform (offline calibration) in the rig.

    The caller resets ``rig.stage_frame`` when the reference changes (the old
    frame placed the old reference).
    """
    rig.reference = reference
    rig.sensors.setdefault(reference, SensorConfig(reference))
    set_calibration(rig, sensor, to_reference, method, fitness, rms_m)
